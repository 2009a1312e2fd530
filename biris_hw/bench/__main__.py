"""``python -m biris_hw.bench``: run the suite and write the reports."""

import sys

from biris_hw.bench.harness import main

sys.exit(main())
