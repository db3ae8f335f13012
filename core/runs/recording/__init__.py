"""A run's every step, recorded as it happens and read back (:mod:`.format` describes the files):
:class:`~.writer.RecordingWriter` appends, :func:`open` reads::

    from .. import recording
    rec = recording.open("out/run0")
"""

from . import format, segments
from .format import FOLDER, INDEX, STEPS, VERSION, RecordingError, ResumePayload
from .reader import Recording, open
from .writer import RecordingWriter

__all__ = [
    "FOLDER",
    "INDEX",
    "STEPS",
    "VERSION",
    "format",
    "segments",
    "Recording",
    "RecordingError",
    "RecordingWriter",
    "ResumePayload",
    "open",
]
