"""The engine options `dsr-bench generate` and `dsr-bench evaluate` share (`dsr_bench.engines`), declared once:
annotate a command's parameter with one of these types and give it the default shown."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from dsr_bench.engines import HELP

RayAddress = Annotated[Optional[str], typer.Option("--ray", metavar="ADDRESS", help=HELP["ray"])]  # default None
Slurm = Annotated[bool, typer.Option("--slurm", help=HELP["slurm"])]  # default False
SlurmPartition = Annotated[Optional[str], typer.Option("--slurm-partition", help=HELP["slurm_partition"])]
SlurmTime = Annotated[Optional[int], typer.Option("--slurm-time", metavar="MINUTES", help=HELP["slurm_time"])]
SlurmTasks = Annotated[Optional[int], typer.Option("--slurm-tasks", help=HELP["slurm_tasks"])]
SlurmLogs = Annotated[Optional[Path], typer.Option("--slurm-logs", help=HELP["slurm_logs"])]
SlurmLocal = Annotated[bool, typer.Option("--slurm-local", help=HELP["slurm_local"])]  # default False
