"""Training the reference models: the paper's curriculum as data (`schedules`), checkpoints
(`checkpoints`) and the trainer (`trainer`). Needs torch."""
