"""``make bench``: the benchmark suite from a checkout; the code lives in ``biris_hw.bench``."""

import sys
from pathlib import Path

# Run the checkout's code even where the project is not installed into the interpreter.
sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from biris_hw.bench import main

if __name__ == "__main__":
    sys.exit(main())
