"""When a control cycle overran: one rule for the loop's statistics (runtime/loop.py), the
recordings' ``/rocoma/manager`` (record/live_channels.py) and the live view's
(live/server.py): one rule, wherever it is counted (each from its own first row).

A cycle overran when it ended after the next cycle's deadline: its lateness (start minus
deadline) and its work (start to the end of ``on_cycle``) together took more than a period.
A cycle that started on time and worked too long is one: the loop does not burst to catch
up but starts the next cycle at once, on time by its new deadline, so a count of late
starts alone would see none of the overruns the work makes.
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
