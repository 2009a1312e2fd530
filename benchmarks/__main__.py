"""``python -m benchmarks``: run the suite and write the reports."""

import sys

from benchmarks.harness import main

sys.exit(main())
