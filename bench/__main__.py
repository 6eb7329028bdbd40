"""`python -m bench` is the `drivebench` command."""

import sys

from bench.faces.cli import main

sys.exit(main())
