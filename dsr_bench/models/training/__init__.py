"""Training the reference models (needs torch): the recipes of `dsr-bench train`, one per kind of model and
track (`tracks`, torch-free), the paper's curriculum as data (`schedules`), what a run is told
(`config.TrainConfig`), the one weights format (`checkpoints`), the run's setup (`setup`: model, optimiser,
scheduler, resume) and data (`loaders`: windows, sampler, DataLoaders), the one loop (`loop`) and the full
track's run of it (`trainer`: `train(config)`, `train_step`, `validate`), its stages in turn (`curriculum`:
`--stage curriculum`, resumable, with a budget); the CPU-sized recipes (`cpu_track`, `image_track`)."""
