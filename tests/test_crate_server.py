"""The VME crate's monitor in the server: ``status().crate``, alarms, a crate that goes quiet, and
what carries it (the wire format, diagnostics, ``biris watch``, target files). Issue 13 B.3.

The crate is a simulated Wiener crate on a python-can ``virtual`` channel of the rig's own
(``SimulatedBiris(crate=True)``), polled every 50 ms of real time: the crate monitor is not a
part of the sensor's hardware time, so nothing here depends on ``time_scale``.
"""

from __future__ import annotations

import json
import logging
import uuid
from pathlib import Path

import pytest

from biris_hw import BirisServer, Direction
from biris_hw.commands.watch import crate_summary, status_line
from biris_hw.crate import CrateMonitor
from biris_hw.errors import RequestError
from biris_hw.io.codec import decode_status, diagnostics, encode_status, typestore
from biris_hw.server.crate_watch import CrateWatch
from biris_hw.status import ServerState
from biris_hw.target import load_target
from regs.wiener_crate import CrateReading
from sim import SimulatedBiris
from tests.conftest import RigFactory, Run, idle_status

WAIT = 10.0


def _fresh(server: BirisServer, polls: int = 2) -> None:
    """Wait until the crate has been read ``polls`` more times (a change is then seen)."""
    watch = server.crate_watch
    assert watch is not None
    assert watch.wait_polls(watch.polls + polls, WAIT), "the crate was not polled"


@pytest.fixture
def crate_rig(make_rig: RigFactory) -> SimulatedBiris:
    return make_rig(crate=True)


def test_a_server_without_a_crate_monitor_says_nothing_of_one(rig: SimulatedBiris) -> None:
    with BirisServer(rig.hardware) as server:
        status = server.status()
        assert server.crate_watch is None
        assert status.crate is None and status.crate_error is None
        assert crate_summary(status) is None
        assert "crate=" not in status_line(status, 0.0)


def test_status_carries_the_crates_reading_and_the_sensor_scans_beside_it(
    crate_rig: SimulatedBiris,
) -> None:
    with BirisServer(crate_rig.hardware) as server:
        _fresh(server, 1)
        status = server.status()
        crate = status.crate
        assert isinstance(crate, CrateReading)
        assert crate.crate_id == 1 and crate.power_on and crate.fans_ok
        assert crate.alarms() == () and status.crate_error is None
        assert crate.voltages_v[0] == pytest.approx(crate_rig.crate.voltages_v[0], abs=0.01)
        # a fan fails: the next readings say so, and the sensor does not care
        crate_rig.crate.fail_fan(2)
        _fresh(server)
        crate = server.status().crate
        assert crate is not None and not crate.fans_ok
        assert crate.fans_rps[2] == 0  # fans 0-5
        assert any("fan" in alarm for alarm in crate.alarms())
        conn = server.open()
        conn.single_scan(30.0)
        conn.wait_idle(timeout=WAIT)
        scan = conn.request_scan_data(Direction.CCW)
        # the sensor scans beside the crate's alarm: whole, or (a host too loaded for scaled
        # time) cut and marked so
        assert scan is not None and (scan.n_acq > 0 or bool(scan.partial_reason))
        assert server.status().state is ServerState.IDLE


def test_a_crate_that_stops_answering_keeps_its_last_reading_and_says_why(
    crate_rig: SimulatedBiris, caplog: pytest.LogCaptureFixture
) -> None:
    with BirisServer(crate_rig.hardware) as server:
        _fresh(server, 1)
        good = server.status().crate
        assert good is not None
        caplog.set_level(logging.WARNING, logger="biris_hw.server")
        crate_rig.crate.go_silent()
        _fresh(server, 3)
        status = server.status()
        assert status.crate_error is not None and "crate 1" in status.crate_error
        assert status.crate == good  # the last good reading, same read_at: its age shows
        assert crate_summary(status) == "unreachable"
        assert status.state is ServerState.IDLE  # the sensor is not the crate
        lost = [r for r in caplog.records if "VME crate:" in r.getMessage()]
        assert len(lost) == 1  # said once, not at every poll
        crate_rig.crate.answer_again()
        _fresh(server)
        status = server.status()
        assert status.crate_error is None
        assert status.crate is not None and status.crate.read_at > good.read_at
        assert any("answers again" in r.getMessage() for r in caplog.records)


def test_an_alarm_is_logged_once_when_it_appears_and_once_when_it_clears(
    crate_rig: SimulatedBiris, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.WARNING, logger="biris_hw.server")
    with BirisServer(crate_rig.hardware) as server:
        _fresh(server, 1)
        crate_rig.crate.over_current(1)
        _fresh(server, 3)
        raised = [r.getMessage() for r in caplog.records if "channel 1" in r.getMessage()]
        assert len(raised) == 1 and "cleared" not in raised[0]
        crate_rig.crate.clear_all()
        _fresh(server, 3)
        said = [r.getMessage() for r in caplog.records if "channel 1" in r.getMessage()]
        assert len(said) == 2 and said[1].startswith("VME crate 1: cleared")


def test_the_crate_reaches_network_clients_diagnostics_and_watch(
    crate_rig: SimulatedBiris,
) -> None:
    with BirisServer(crate_rig.hardware) as server:
        crate_rig.crate.overheat(3)
        _fresh(server)
        status = server.status()
    crate = status.crate
    assert crate is not None and crate.supply_temperature == 1 << 3
    # the wire: the same reading back, every field
    back = decode_status(encode_status(status, 1.0))
    assert back.crate == crate and back.crate_error is None
    # diagnostics: one status for the crate, ERROR with its alarm
    encoded = diagnostics(status, 1.0)
    msg = typestore().deserialize_cdr(encoded.data, encoded.msgtype)
    (item,) = [s for s in msg.status if s.name == "VME crate"]
    assert item.level == 2 and "channel 3" in item.message
    values = {kv.key: kv.value for kv in item.values}
    assert values["power"] == "on" and values["fan1.rpm"] == str(crate.fans_rps[0] * 60)
    # watch: a field in line mode
    assert "crate=" in status_line(status, 0.0) and "channel_3" in status_line(status, 0.0)


def test_an_unreachable_crate_crosses_the_wire_as_an_error() -> None:
    status = idle_status(crate_error="no answer from crate 7")
    back = decode_status(encode_status(status))
    assert back.crate is None and back.crate_error == "no answer from crate 7"
    encoded = diagnostics(status, 0.0)
    msg = typestore().deserialize_cdr(encoded.data, encoded.msgtype)
    (item,) = [s for s in msg.status if s.name == "VME crate"]
    assert item.level == 1 and item.message == "no answer from crate 7"


def test_the_poll_period_is_checked() -> None:
    with pytest.raises(ValueError, match=r"at least 0\.01 s"):
        CrateWatch(object(), 0.0)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=r"at least 0\.01 s"):
        CrateWatch(object(), float("nan"))  # type: ignore[arg-type]


# -- target files ---------------------------------------------------------------------------------


def _target(tmp_path: Path, crate: str, axes: str = "") -> Path:
    images = {}
    for name, size in (("biris", 0x84000), ("motion", 0x100), ("coupler", 0x20)):
        images[name] = tmp_path / f"{name}.img"
        images[name].write_bytes(bytes(size))
    motion = (
        ""
        if axes
        else f'motion = {{ kind = "mmap", path = "{images["motion"]}", size = 0x100 }}\n'
        'level3 = { kind = "eventfd" }\n'
    )
    path = tmp_path / "robot.toml"
    path.write_text(
        f"""
biris = {{ kind = "mmap", path = "{images["biris"]}", size = 0x84000 }}
coupler = {{ kind = "mmap", path = "{images["coupler"]}" }}
level2 = {{ kind = "eventfd" }}
{motion}pan_journal = ""
{axes}
[crate]
{crate}
"""
    )
    return path


def test_a_crate_table_opens_a_monitor_the_server_polls(tmp_path: Path) -> None:
    from sim.wiener_crate import SimulatedCrate

    channel = f"crate-{uuid.uuid4().hex}"
    path = _target(
        tmp_path,
        f'kind = "wiener-can"\ninterface = "virtual"\nchannel = "{channel}"\ncrate_id = 9\n'
        "poll = 0.5\ntimeout = 0.1\n",
    )
    hardware = load_target(path)
    try:
        assert isinstance(hardware.crate, CrateMonitor)
        assert hardware.crate.crate_id == 9 and hardware.crate_poll_s == 0.5
        with SimulatedCrate(channel, 9) as crate:
            reading = hardware.crate.read()
            assert reading.crate_id == 9 and reading.ok
            assert crate.violations == []
    finally:
        hardware.close()


@pytest.mark.parametrize(
    ("crate", "message"),
    [
        ('kind = "wiener"\ncrate_id = 1', r"crate\.kind: must be one of wiener-can"),
        ('kind = "wiener-can"', r"crate\.crate_id: missing"),
        ('kind = "wiener-can"\ncrate_id = 0', r"crate\.crate_id: must be in 0x1\.\.0x7E"),
        ('kind = "wiener-can"\ncrate_id = 1.5', r"crate\.crate_id: must be an integer"),
        ('kind = "wiener-can"\ncrate_id = 1\npoll = 0', r"crate\.poll: must be a positive"),
        ('kind = "wiener-can"\ncrate_id = 1\nchanel = "can0"', r"crate\.chanel: not an option"),
        ('kind = "wiener-can"\ncrate_id = 1\nchannel = 3', r"crate\.channel: must be a string"),
    ],
)
def test_crate_mistakes_name_their_key(tmp_path: Path, crate: str, message: str) -> None:
    with pytest.raises(RequestError, match=message):
        load_target(_target(tmp_path, crate))


def test_a_crate_on_the_drives_bus_may_not_take_a_drives_node_id(tmp_path: Path) -> None:
    channel = f"t-{uuid.uuid4().hex}"
    axes = (
        f'[axes]\nkind = "cia402"\ninterface = "virtual"\nchannel = "{channel}"\n'
        "pan_node = 2\ntilt_node = 3\n"
    )
    crate = f'kind = "wiener-can"\ninterface = "virtual"\nchannel = "{channel}"\ncrate_id = 3\n'
    with pytest.raises(RequestError, match=r"crate\.crate_id: 3 is a drive's node id"):
        load_target(_target(tmp_path, crate, axes))


def test_regdump_shows_a_targets_crate_and_a_silent_one(tmp_path: Path, biris: Run) -> None:
    from sim.wiener_crate import SimulatedCrate

    channel = f"crate-{uuid.uuid4().hex}"
    path = _target(
        tmp_path,
        f'kind = "wiener-can"\ninterface = "virtual"\nchannel = "{channel}"\ncrate_id = 4\n'
        "timeout = 0.05\n",
    )
    with SimulatedCrate(channel, 4) as crate:
        crate.fail_fan(0)
        code, out, err = biris("regdump", "--target", str(path), "--json")
        assert code == 0, err
        section = json.loads(out)["crate"]
        assert section["title"] == "Wiener VME crate 4" and section["power"] is True
        assert section["fans"][0] == 0 and any("fan" in a for a in section["alarms"])
        assert section["channel 0"][0] == pytest.approx(crate.voltages_v[0], abs=0.01)
        code, out, err = biris("regdump", "--target", str(path))
        assert code == 0, err
        assert "Wiener VME crate 4" in out and "fan failure" in out
    # the crate gone: the boards are still dumped, and the crate's row says why it is empty
    code, out, err = biris("regdump", "--target", str(path), "--json")
    assert code == 0, err
    dump = json.loads(out)
    assert "no answer" in dump["crate"]["answer"] and "crate 4" in dump["crate"]["answer"]
    assert "biexec" in dump and "coupler" in dump
