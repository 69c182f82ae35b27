"""When a control cycle overran: one rule for the loop's statistics (runtime/loop.py), the
recordings' ``/rocoma/manager`` (record/live_channels.py) and the live view's
(live/server.py): one rule, wherever it is counted (each from its own first row).

A cycle overran when it ended after the next cycle's deadline: its lateness (start minus
deadline) and its work (start to the end of ``on_cycle``) together took more than a period.
A cycle that started on time and worked too long is one: the loop does not burst to catch
up but starts the next cycle at once, on time by its new deadline, so a count of late
starts alone would see none of the overruns the work makes.

An overrun *waited* when the cycle spent more of its time off the CPU than on it (its late
start; its work preempted, or waiting for the GIL, a lock or I/O): scheduling, another
thread or process, is the cause, what a real-time priority and a CPU of the loop's own
address. The others were mostly CPU work: a cycle too heavy for the period, or a CPU that
ran slow (a virtual machine's host). ``cpu`` is the loop thread's CPU time in the work.
"""
from __future__ import annotations

from typing import TYPE_CHECKING, Any, overload

if TYPE_CHECKING:
    from numpy import bool_, float64
    from numpy.typing import NDArray


@overload
def overran(work: float, late: float, period: float) -> bool: ...
@overload
def overran(work: NDArray[float64], late: NDArray[float64],
            period: float) -> NDArray[bool_]: ...


def overran(work: Any, late: Any, period: float) -> Any:
    """Seconds of work and lateness of one cycle (scalars) or of a block of recorded rows
    (arrays); ``period``: the loop's."""
    return late + work > period


@overload
def waited(work: float, late: float, cpu: float) -> bool: ...
@overload
def waited(work: NDArray[float64], late: NDArray[float64],
           cpu: NDArray[float64]) -> NDArray[bool_]: ...


def waited(work: Any, late: Any, cpu: Any) -> Any:
    """Of an overrun: off the CPU longer than on it (scalars, or arrays of rows)."""
    return late + work > 2.0 * cpu
