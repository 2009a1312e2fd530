"""``BirisSupervisor``: the 68020/OS-9 supervisor that executes BIEXEC_COM commands.

The driver reaches BIRIS only through memory (BIEXEC_COM, the frames, the azimuth table) and
level-2 interrupts, so the model works the same way: it shares a buffer window with the driver
and raises interrupts through an :class:`~sim.irqgate.InterruptGate`. How we read the report
(docs/design.md), where it is silent, is told where it is done:
:mod:`~sim.supervisor.commands` (vertical sync, busy), :mod:`~sim.supervisor.acquisition`
(BI_ACQUIRE, continuous acquisition, the exposure audits), :mod:`~sim.supervisor.boot`
(calibration), :mod:`~sim.supervisor.faults` (injected faults); the thread and what it lets
others see are in :mod:`~sim.supervisor.supervisor`, the shared fields in
:mod:`~sim.supervisor.state`, the field grid in :mod:`~sim.supervisor.schedule`.
"""

from sim.supervisor.state import AcquireFn, GarbageKind
from sim.supervisor.supervisor import BirisSupervisor

__all__ = ["AcquireFn", "BirisSupervisor", "GarbageKind"]
