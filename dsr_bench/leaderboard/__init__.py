"""The leaderboard: entries recomputed from predictions (or plans) and validated (`entries`), and the tables built
from them (`board`: `add_entry`, `build`). It sits above scoring, the models and the planning track, whose results it
ranks; none of them imports it."""
