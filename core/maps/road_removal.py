"""Road removal of a cached prior map in a child process.

open3d's normal estimation holds Python's GIL for its whole run (~10 s on the built-in town's
map): in a thread of the localizer's process it would stall the filter, the viewer and every
other thread that long (measured: the first scan of a viewer's first start came 9 s late). In a
child process it stalls nothing. It runs in its own session (its own scheduler group, see
:func:`~lidarloc.core.worker_process.lower_priority`) at normal priority: the filter cannot say
"localized" before S2M has confirmed it, and S2M needs this map, so starving it starves the run
(measured on a machine at load 8: niced by 10, it had done 15 % after 80 s and the viewer never
left "PF only"). The filter's step needs ~10 ms of the 100 ms between scans, so sharing the cores
with it for the ~10 s it takes costs the playback nothing.

``python -m lidarloc.core.maps.road_removal MAP_DIR MAP_CONFIG_JSON NICE`` adds the road-removed map to
the map's cache directory (:func:`~lidarloc.core.maps.mapping.load_or_build_road_removed`).
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
import threading
from dataclasses import asdict
from pathlib import Path

from ..config import MapConfig
from ..errors import LidarlocError


class RoadRemovalProcess:
    """The child process removing the road from the map cached in ``map_dir``. ``progress`` is
    the share of the map done so far (0…1), as the child reports it on its standard output."""

    def __init__(self, map_dir: Path, cfg: MapConfig, nice: int = 0):
        self.progress = 0.0
        self._err = tempfile.TemporaryFile()  # a file, not a pipe: a chatty child never blocks
        self._proc = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "lidarloc.core.maps.road_removal",
                str(map_dir),
                json.dumps(asdict(cfg)),
                str(int(nice)),
            ],
            stdout=subprocess.PIPE,
            stderr=self._err,
            start_new_session=True,
        )
        self._reader = threading.Thread(target=self._read_progress, name="lidarloc-road-removal-progress", daemon=True)
        self._reader.start()

    def _read_progress(self) -> None:
        for line in self._proc.stdout:
            try:
                self.progress = float(line.decode().split()[-1])
            except (ValueError, IndexError):
                pass

    def wait(self) -> None:
        """Block until it is done; a failure raises :class:`LidarlocError` with the child's last line."""
        self._proc.wait()
        self._reader.join()
        self._err.seek(0)
        err = self._err.read()
        self._err.close()
        if self._proc.returncode != 0:
            lines = [ln for ln in err.decode(errors="replace").splitlines() if ln.strip()]
            raise LidarlocError(f"road removal failed: {lines[-1] if lines else f'exit code {self._proc.returncode}'}")

    def kill(self, wait: bool = True) -> None:
        """SIGKILL the child (its map is written to a temporary name, then renamed: nothing is
        left half-written); ``wait`` False does not reap it (the parent is about to exit)."""
        if self._proc.poll() is None:
            self._proc.kill()
            if wait:
                self._proc.wait()


def main(argv: list[str]) -> int:
    from ..worker_process import lower_priority
    from .mapping import PriorMap, load_or_build_road_removed

    map_dir, cfg_json, nice = Path(argv[0]), argv[1], int(argv[2])
    lower_priority(nice)
    meta = json.loads((map_dir / "meta.json").read_text())

    def report(fraction: float) -> None:
        print(f"progress {fraction:.3f}", flush=True)

    load_or_build_road_removed(PriorMap.load(map_dir, meta), map_dir, MapConfig(**json.loads(cfg_json)), report)
    return 0


if __name__ == "__main__":
    try:
        sys.exit(main(sys.argv[1:]))
    except LidarlocError as exc:
        print(f"error: {exc}", file=sys.stderr)
        sys.exit(2)
