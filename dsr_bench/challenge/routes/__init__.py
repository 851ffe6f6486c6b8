"""The challenge server's routes, one router per concern (`server.create_app` mounts them all):

- `deps`: the app's context (layout, settings, database, throttle, session signer, the configuration) and the FastAPI
  dependencies of every route: the database session, the team of a Bearer token (`api_team`) or of a browser's
  session cookie (`browser_team`).
- `uploads`: `POST /api/submissions` (streamed under the size and time limits, multipart or raw body).
- `submissions`: a submission's status and result file, the final choice, the team's history (JSON).
- `teams`: signing in and out in a browser, the team's own page (history, final choices), a team's public page.
- `pages`: the leaderboard (page and JSON), a submission's page, the participants' guide, the inputs.
- `admin`: the health check.
"""
