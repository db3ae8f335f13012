"""``lidarloc corpus example``: a corpus of the built-in town's drives, ready to run.

Drive i is town seed i // 4 scanned by the i-th of the town's sensors in turn (HDL-64E, VLP-16,
VLP-32C, OS1-128), all in the lived-in world (objects changed since mapping, traffic, scans swept
while moving): the drives differ in what makes localization hard — the town, the sensor's
resolution — and every four drives share one town, so its map is built once for them. Each drive
meets its own day's traffic (``town.traffic_seed`` = its number) on the same changed streets.

With ``seeds`` > 1 each drive is repeated under seeds 0 … seeds − 1 (``NAME-sK``): one log under
several seeds, from which ``lidarloc corpus compare`` measures the seed-to-seed noise.
"""

from __future__ import annotations

from ...core.config import TOWN_SENSORS

WORLD = "lived-in"


def example_drives(drives: int, seeds: int = 1) -> list[dict]:
    """The corpus's drives as the file writes them."""
    out = []
    for i in range(drives):
        town, sensor = divmod(i, len(TOWN_SENSORS))
        name = TOWN_SENSORS[sensor]
        # each drive its own day: other traffic on the same changed streets (town.traffic_seed)
        drive = {
            "name": f"town{town}-{name}",
            "town_seed": town,
            "set": [f"town.sensor={name}", f"town.traffic_seed={i}"],
        }
        if seeds == 1:
            out.append(drive)
            continue
        out += [{**drive, "name": f"{drive['name']}-s{k}", "seed": k} for k in range(seeds)]
    return out


def example_corpus(drives: int, scans: int | None, seeds: int = 1) -> str:
    """The corpus file's text: a comment saying what it is, the defaults, the drives."""
    import yaml

    defaults: dict = {"world": WORLD, "seed": 0}
    if scans is not None:
        defaults["scans"] = scans
    repeated = "" if seeds == 1 else f", each under seeds 0…{seeds - 1}"
    header = (
        f"# {drives} drives of the built-in town: town seeds × sensors{repeated}, in the {WORLD} world.\n"
        "# Run it with: lidarloc corpus run THIS_FILE --out DIR  (the format: docs/corpus.md)\n"
    )
    body = yaml.safe_dump(
        {"defaults": defaults, "drives": example_drives(drives, seeds)},
        sort_keys=False,
        allow_unicode=True,
        default_flow_style=None,
    )
    return header + body
