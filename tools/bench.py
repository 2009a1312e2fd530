"""``make bench``: the benchmark suite from a checkout; the code lives in ``benchmarks/``.

The same as ``python -m benchmarks`` run from the checkout's root, from any directory. The
``benchmarks`` folder is not part of the installed distribution (it imports ``sim`` freely), so
this script puts the checkout's root on the import path first.
"""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks import main

if __name__ == "__main__":
    sys.exit(main())
