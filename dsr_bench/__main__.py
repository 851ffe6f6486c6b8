"""`python -m dsr_bench`: the `dsr-bench` command line."""

import sys

from dsr_bench.cli import main

sys.exit(main())
