"""The layers hold at run time: importing a low layer does not load a higher one.

Each check runs in a fresh interpreter, since this one has long since imported everything. The
static rules (who may import whom) are import-linter's contracts in pyproject.toml.
"""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

import biris_hw


def _loaded_after(statement: str) -> list[str]:
    """The ``biris_hw``/``sim`` modules a fresh interpreter holds after ``statement``."""
    probe = (
        f"{statement}\n"
        "import json, sys\n"
        "ours = [m for m in sys.modules if m.split('.')[0] in {'biris_hw', 'sim'}]\n"
        "print(json.dumps(sorted(ours)))"
    )
    done = subprocess.run(
        [sys.executable, "-c", probe], capture_output=True, text=True, timeout=60, check=False
    )
    assert done.returncode == 0, done.stderr
    loaded: list[str] = json.loads(done.stdout)
    return loaded


@pytest.mark.parametrize(
    "statement",
    [
        "import biris_hw",
        "import biris_hw.bus",
        "import biris_hw.irq",
        "import biris_hw.hardware",
        "from biris_hw import BirisHardware, Scan, deg_to_counts",
        "import sim",
        "from sim import SimulatedBiris, Scene",
    ],
)
def test_below_the_server_nothing_loads_it(statement: str) -> None:
    loaded = _loaded_after(statement)
    assert [m for m in loaded if m.startswith("biris_hw.server")] == []
    assert [m for m in loaded if m.startswith(("biris_hw.client", "biris_hw.commands"))] == []


def test_the_bus_layer_loads_no_simulator_and_no_interrupt_lines() -> None:
    loaded = _loaded_after("import biris_hw.bus")
    assert [m for m in loaded if m.startswith(("sim", "biris_hw.irq", "biris_hw.hardware"))] == []


def test_the_root_still_offers_every_public_name() -> None:
    loaded = _loaded_after(
        "from biris_hw import *\n"
        "from biris_hw import __all__\n"
        "missing = [n for n in __all__ if n not in globals()]\n"
        "assert not missing, missing"
    )
    assert "biris_hw.server" in loaded
    assert sorted(biris_hw._WHERE) == sorted(biris_hw.__all__)
    assert sorted(dir(biris_hw)) == sorted(set(dir(biris_hw)) | set(biris_hw.__all__))
    with pytest.raises(AttributeError, match="no attribute 'Nope'"):
        _ = biris_hw.Nope  # type: ignore[attr-defined]
