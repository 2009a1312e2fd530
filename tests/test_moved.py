"""The old import paths of the modules now in biris_hw.io (and biris_hw.remote, now
biris_hw.simlink) keep working for one release: the same module object, with a warning."""

from __future__ import annotations

import importlib
import sys

import pytest

from biris_hw._moved import MOVED, new_name


@pytest.mark.parametrize("old", sorted(MOVED))
def test_an_old_path_is_the_new_module_and_warns(old: str) -> None:
    new = importlib.import_module(MOVED[old])
    sys.modules.pop(old, None)  # as in a fresh process, where nothing imported it yet
    with pytest.warns(DeprecationWarning, match=f"{old} moved to {MOVED[old]}"):
        module = importlib.import_module(old)
    assert module is new
    assert sys.modules[old] is new


def test_a_submodule_of_a_moved_package_follows_it() -> None:
    assert new_name("biris_hw.net.service") == "biris_hw.io.net.service"
    assert new_name("biris_hw.net.protocol") == "biris_hw.io.net.keys"
    assert new_name("biris_hw.records") is None  # a prefix of a name is not the name
    sys.modules.pop("biris_hw.record.recorder", None)
    with pytest.warns(DeprecationWarning):
        from biris_hw.record.recorder import Recorder
    from biris_hw.io.record import Recorder as Now

    assert Recorder is Now


def test_the_names_of_design_3b_still_import() -> None:
    """DESIGN.md 3b's import lines, as a user's script has them."""
    for old in ("biris_hw.net", "biris_hw.record", "biris_hw.replay"):
        sys.modules.pop(old, None)
    with pytest.warns(DeprecationWarning):
        from biris_hw.net import connect, serve
        from biris_hw.record import Recorder
        from biris_hw.replay import ReplayServer
    from biris_hw.io.net import connect as now_connect
    from biris_hw.io.record import Recorder as NowRecorder
    from biris_hw.io.record import ReplayServer as NowReplay

    assert (connect, Recorder, ReplayServer) == (now_connect, NowRecorder, NowReplay)
    assert callable(serve)
