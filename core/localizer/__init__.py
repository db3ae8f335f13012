"""The localizer: the scan loop that drives the blocks (PF, RPE, RS, S2M + SU) in threads and
child processes, its lifecycle, clocks and live parameters (:mod:`.scan_loop`).
"""

from .blocks import INTERRUPT_POLL_S, BlockError, Interrupted
from .scan_loop import Localizer
from .tables import S2M_READY_DETAIL

__all__ = ["INTERRUPT_POLL_S", "S2M_READY_DETAIL", "BlockError", "Interrupted", "Localizer"]
