"""``lidarloc corpus example``: a corpus of the built-in town's drives, ready to run.

Drive i is town seed i // 4 scanned by the i-th of the town's sensors in turn (HDL-64E, VLP-16,
VLP-32C, OS1-128), all in the lived-in world (objects changed since mapping, traffic, scans swept
while moving): the drives differ in what makes localization hard — the town, the sensor's
resolution — and every four drives share one town, so its map is built once for them.
"""

from __future__ import annotations

from ...core.config import TOWN_SENSORS

WORLD = "lived-in"


def example_drives(drives: int) -> list[dict]:
    """The corpus's drives as the file writes them."""
    out = []
    for i in range(drives):
        seed, sensor = divmod(i, len(TOWN_SENSORS))
        name = TOWN_SENSORS[sensor]
        out.append({"name": f"town{seed}-{name}", "town_seed": seed, "set": [f"town.sensor={name}"]})
    return out


def example_corpus(drives: int, scans: int | None) -> str:
    """The corpus file's text: a comment saying what it is, the defaults, the drives."""
    import yaml

    defaults: dict = {"world": WORLD, "seed": 0}
    if scans is not None:
        defaults["scans"] = scans
    header = (
        f"# {drives} drives of the built-in town: town seeds × sensors, in the {WORLD} world.\n"
        "# Run it with: lidarloc corpus run THIS_FILE --out DIR  (the format: docs/corpus.md)\n"
    )
    body = yaml.safe_dump(
        {"defaults": defaults, "drives": example_drives(drives)},
        sort_keys=False,
        allow_unicode=True,
        default_flow_style=None,
    )
    return header + body
