"""``lidarloc export RUN --out NAME``: a recorded run as files anyone can open — a viser
recording of its scene (``NAME.viser``) and a self-contained static web folder (``NAME/``: viser's
own client build as ``index.html`` and the recording) that plays it from disk with no server and
no Python: open ``NAME/index.html`` in a browser, or zip the folder and attach it to a bug report.

The page reads the recording from ``NAME/recording.js`` (the ``.viser`` file's bytes, base64 in a
script), because a page opened from ``file://`` may load scripts but may not fetch files. The
``.viser`` file plays in any viser client that is served over HTTP
(``index.html?playbackPath=NAME.viser``); it is kept beside the folder, not in it, so that the
folder to share holds the recording once.

Each step of the run is 0.1 s of the recording (the LiDAR's 10 Hz): the player's play, pause,
speed and time slider scrub the run step by step. What the viewer's panel would say (scan,
localized, std, error, N_eff) is drawn with the scene (:mod:`.export_scene`): a label at the
estimate and an overlay in the page's corner.

The map and the scans come from the run's source, which the recording names (one-line error if
it moved); the map is thinned for display so that a 300-scan run of a real drive stays well under
100 MB.

Why viser's own serializer and not ``viser4d`` (a viser extension with a time-indexed scene, a
scrub/step overlay and an HTML export): it was tried on the same 50-step scene and works (same
sizes, plays offline from ``file://``), but it is an alpha by one author that reaches into viser's
private internals (hence its pin below viser 1.2), needs Python ≥ 3.11 and numpy ≥ 2.4 where
lidarloc supports Python 3.10 and numpy 1.24, and brings a dependency we do not use
(``viser-audio``). viser's serializer and its embedded player do all that export needs.
"""

from __future__ import annotations

import base64
import contextlib
import io
import re
import time
from pathlib import Path

import numpy as np
from rich.console import Console

from ..core.errors import LidarlocError
from .export_scene import EXPORT_MAP_POINTS, ExportScene

#: seconds of the recording per step of the run (the LiDAR's period)
STEP_SECONDS = 0.1
PAGE = "index.html"
DATA_SCRIPT = "recording.js"


def client_page() -> str:
    """viser's single-file client build (the page that plays embedded recordings)."""
    import viser

    path = Path(viser.__file__).parent / "client" / "build" / "index.html"
    try:
        html = path.read_text(encoding="utf-8")
    except OSError:
        html = ""
    major = int(str(getattr(viser, "__version__", "0")).split(".")[0] or 0)
    # the build is compressed: the page's support for embedded recordings is told by the version
    if major < 1 or "</head>" not in html:
        raise LidarlocError(
            f"viser {getattr(viser, '__version__', '?')}: its client build ({path}) cannot play "
            "an embedded recording; export needs viser ≥ 1.0"
        )
    return html


def page_html(client: str, title: str) -> str:
    """The client page, told to load the recording from DATA_SCRIPT and to start dark (the
    viewer's colours are made for a dark background)."""
    inject = f'<script>window.__VISER_EMBED_CONFIG__={{darkMode:true}};</script><script src="{DATA_SCRIPT}"></script>'
    head_end = client.index("</head>")
    page = client[:head_end] + inject + client[head_end:]
    return re.sub(r"<title>[^<]*</title>", lambda _: f"<title>{_escape(title)}</title>", page, count=1)


def _escape(text: str) -> str:
    return text.replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;")


def _hud_sender(server):
    """A function running JavaScript in the recorded page (the overlay), or None where this viser
    has no way to: the label at the estimate still carries the figures. viser has no public call
    for it; this is the message its own plotly support sends, recorded like any scene message."""
    try:
        from viser._messages import RunJavascriptMessage

        queue = server._websock_server.queue_message
    except (ImportError, AttributeError):
        return None
    return lambda source: queue(RunJavascriptMessage(source=source))


def _camera(server, rec) -> None:
    """Look at the drive from above and behind, the whole trajectory in view."""
    pts = np.concatenate([rec.gt_pose[:, :3, 3], rec.mean_pose[rec.localized.astype(bool), :3, 3]])
    pts = pts[np.isfinite(pts).all(axis=1)]
    if not len(pts):
        pts = rec.mean_pose[:, :3, 3]
        pts = pts[np.isfinite(pts).all(axis=1)]
    if not len(pts):
        return  # nothing to look at: viser's default view
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    center = (lo + hi) / 2.0
    ext = float(max(hi[0] - lo[0], hi[1] - lo[1], 60.0))
    server.initial_camera.up = (0.0, 0.0, 1.0)
    server.initial_camera.look_at = tuple(float(v) for v in center)
    server.initial_camera.position = tuple(float(v) for v in center + np.array([0.0, -0.55 * ext, 0.75 * ext]))


def _out_paths(out: Path) -> tuple[Path, Path]:
    """(the web folder, the .viser file beside it) that ``--out`` names."""
    out = Path(out).expanduser()
    if out.suffix == ".viser":
        out = out.with_suffix("")
    if not out.name:
        raise LidarlocError(f"{out}: name the export (--out NAME writes NAME.viser and the folder NAME/)")
    if out.exists() and not out.is_dir():
        raise LidarlocError(f"{out}: exists and is not a folder; --out NAME writes NAME.viser and the folder NAME/")
    return out, out.with_name(out.name + ".viser")


def export_run(
    run_dir,
    out,
    console: Console | None = None,
    cache_root: Path | None = None,
    scans: bool = True,
    max_map_points: int = EXPORT_MAP_POINTS,
) -> dict:
    """Export the recorded run ``run_dir`` to the folder ``out`` (see the module docstring).
    ``scans``: draw each step's scan (recomputed from the source). Returns what was written:
    paths, sizes in bytes, steps, map points, seconds."""
    import viser

    from ..core.maps.mapping import load_or_build_map
    from ..core.runs import recording
    from .console import progress_bar

    console = console or Console(stderr=True)
    t0 = time.perf_counter()
    rec = recording.open(run_dir)
    if rec.n == 0:
        raise LidarlocError(f"{rec.path}: the recording has no complete step to export")
    folder, viser_file = _out_paths(out)
    client = client_page()
    seq = rec.open_sequence()
    cfg = rec.config()
    with progress_bar() as bar:  # from the cache; built (minutes) only if the cache lost it
        task = bar.add_task("preparing map", total=100)
        prior = load_or_build_map(
            seq.map_source, cfg.map, cache_root, progress=lambda i, n: bar.update(task, completed=100 * i / max(n, 1))
        ).value
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise LidarlocError(f"{folder}: cannot create the folder ({exc.strerror})") from None

    title = f"lidarloc · {rec.meta.get('sequence', 'run')} · {rec.run_dir.name}"
    # A server only because viser's serializer records what a server sends; it binds the loopback,
    # no browser ever connects, and its banner would tell the user of a server they need not open
    # (stdout also carries --json).
    quiet = contextlib.redirect_stdout(io.StringIO())
    with quiet:
        server = viser.ViserServer(host="127.0.0.1", port=0, label="lidarloc export", verbose=False)
    try:
        serializer = server.get_scene_serializer()
        _camera(server, rec)
        view = ExportScene(server.scene, title, rec.n, hud=_hud_sender(server))
        view.draw_map(prior.points, max_points=max_map_points)
        with progress_bar() as bar:
            task = bar.add_task("exporting steps", total=rec.n)
            for i in range(rec.n):
                view.draw_step(i, rec.snapshot(i, seq if scans else None))
                serializer.insert_sleep(STEP_SECONDS)
                bar.update(task, completed=i + 1)
        data = serializer.serialize()
    finally:
        with quiet:
            server.stop()

    try:
        viser_file.write_bytes(data)
        (folder / DATA_SCRIPT).write_text(
            'window.__VISER_EMBED_DATA__="' + base64.b64encode(data).decode("ascii") + '";\n', encoding="ascii"
        )
        (folder / PAGE).write_text(page_html(client, title), encoding="utf-8")
    except OSError as exc:
        raise LidarlocError(f"{folder}: cannot write the export ({exc.strerror})") from None
    folder_bytes = sum(p.stat().st_size for p in (folder / DATA_SCRIPT, folder / PAGE))
    result = {
        "folder": str(folder),
        "page": str(folder / PAGE),
        "viser": str(viser_file),
        "steps": rec.n,
        "map_points": view.map_points,
        "map_voxel_m": view.map_voxel,
        "viser_bytes": viser_file.stat().st_size,
        "folder_bytes": folder_bytes,
        "seconds": time.perf_counter() - t0,
    }
    console.print(
        f"exported {rec.n} steps of {rec.run_dir}: open {folder / PAGE} in a browser (no server "
        f"needed; the folder is {folder_bytes / 1e6:.1f} MB); the recording: {viser_file} "
        f"({result['viser_bytes'] / 1e6:.1f} MB)"
    )
    return result
