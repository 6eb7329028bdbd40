"""`python -m bench` is the `drivebench` command."""

import sys

from bench.cli import main

sys.exit(main())
