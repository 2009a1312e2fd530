"""The rigs the running test has built, in one module both copies of ``conftest`` share.

pytest loads ``tests/conftest.py`` as ``conftest``, and test modules import it again as
``tests.conftest``: a global there exists twice. :func:`tests.conftest.until` and
:func:`tests.conftest.spawn`, called from a test module, must see the rigs the fixtures (of the
other copy) recorded, so the list lives here.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from sim.rig import SimulatedBiris

rigs: list[SimulatedBiris] = []
"""Every SimulatedBiris built during the running test, oldest first; emptied between tests."""
