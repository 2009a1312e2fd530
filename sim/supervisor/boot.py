"""BI_BOOT and BI_LOAD_LUT: the boot file and calibration tables, from the RAMdisk.

**Calibration.** Booting loads the boot file's default table; BI_LOAD_LUT n loads the table
for elevation n counts (NO_CALIBRATION outside the boot file's range) -- "a calibration must
exist for each angle of elevation that is chosen". A table is in use from its command's
completion on, so an acquisition started before the completion still runs on the old one.
"""

from __future__ import annotations

from regs.biexec import BiStatus
from sim.ramdisk import BootParameters
from sim.supervisor.state import SupervisorState, parse_int

__all__ = ["Boot"]


class Boot(SupervisorState):
    """BI_BOOT and BI_LOAD_LUT."""

    def _cmd_boot(self, done: float) -> None:
        name = self._param_text()
        if self._continuous:
            self._finish_later(done, BiStatus.BAD_PARAM, "continuous acquisition running")
            return
        if name is None or name not in self._ramdisk:
            self._finish_later(done, BiStatus.NO_BOOT_FILE, "no such boot file")
            return
        try:
            params = BootParameters.parse(self._ramdisk.read(name).decode("ascii"))
        except (ValueError, UnicodeDecodeError, FileNotFoundError) as exc:
            self._finish_later(done, BiStatus.BAD_PARAM, f"bad boot file: {exc}")
            return
        if params.samples != self._map.samples:
            self._finish_later(
                done, BiStatus.BAD_PARAM, f"boot file is for {params.samples} samples"
            )
            return
        if params.lut_file not in self._ramdisk:
            self._finish_later(done, BiStatus.NO_CALIBRATION, "no calibration file")
            return

        def apply() -> None:
            self._boot = params
            self._lut = params.lut_default

        self._finish_later(done, BiStatus.OK, "", apply=apply)

    def _cmd_load_lut(self, done: float) -> None:
        text = self._param_text()
        elevation = parse_int(text, signed=True)
        if elevation is None:
            self._finish_later(done, BiStatus.BAD_PARAM, f"bad elevation {text!r}")
            return
        boot = self._boot
        if boot is None:
            self._finish_later(done, BiStatus.NOT_BOOTED, "not booted")
            return
        if not boot.has_calibration(elevation):
            self._finish_later(done, BiStatus.NO_CALIBRATION, f"no table for {elevation}")
            return

        def apply() -> None:
            self._lut = elevation

        self._finish_later(done, BiStatus.OK, "", apply=apply)
