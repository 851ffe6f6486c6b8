"""Training the reference models (needs torch): the paper's curriculum as data (`schedules`), what
a run is told (`config.TrainConfig`), checkpoints (`checkpoints`), the run's setup (`setup`: model,
optimiser, scheduler, resume) and data (`loaders`: windows, sampler, DataLoaders), and the loop
(`trainer`: `train(config)`, `train_step`, `validate`)."""
