"""The `dsr-bench` subcommands, one module per command group; each defines `register(app)`.

Command modules import heavy libraries inside the command functions so `dsr-bench --help` is fast.
"""
