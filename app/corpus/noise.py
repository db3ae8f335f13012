"""How much a figure moves between runs that differ only in their seed: the corpus measures its
own noise, and ``lidarloc corpus compare`` reports only changes beyond it.

Drives of one log under several seeds (same source, configuration and preset; drive.json tells)
form a seed group. A figure's spread in a group is the range (largest − smallest) of its values
over the group's seeds, in BASE or in NEW, whichever is larger: a change of code may make runs
noisier, and a regression must stand out of either run's noise. A drive of a seed group is
weighed against its own group's spread; any other drive against the largest spread of any group
(the corpus's own worst case: fewer false alarms, at the price of missing a change smaller than
that). A figure counts as worse when its change in the worse direction exceeds

    threshold = max(floor, K × spread)

with the floors of :data:`~.figures.FIGURES` and :data:`K`. Without seed groups the floors
alone decide.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from .figures import BY_NAME, FIGURES, CorpusOutput

#: how many seed-to-seed spreads a change must exceed. The range of a few seeds underestimates
#: what another seed could do (two seeds show one difference of two draws); twice it leaves room.
K = 2.0


def _spread(values: list[float | None]) -> float | None:
    known = [v for v in values if v is not None]
    return max(known) - min(known) if len(known) >= 2 else None


@dataclass
class Noise:
    """The seed-to-seed spread of each figure: per seed group (keyed by its drives' names) and
    the largest of any group."""

    groups: dict[frozenset, dict[str, float]] = field(default_factory=dict)
    pooled: dict[str, float] = field(default_factory=dict)
    member: dict[str, list[frozenset]] = field(default_factory=dict)  # drive → its groups (BASE's, NEW's)

    def spread(self, drive: str, figure: str) -> float:
        """The spread ``drive`` is weighed against for ``figure`` (0: no seed group says)."""
        own = [self.groups[g][figure] for g in self.member.get(drive, []) if figure in self.groups[g]]
        if own:
            return max(own)
        return self.pooled.get(figure, 0.0)

    def threshold(self, drive: str, figure: str) -> float:
        return max(BY_NAME[figure].floor, K * self.spread(drive, figure))


def measure_noise(*outputs: CorpusOutput) -> Noise:
    """The seed groups of every output and each figure's spread in them."""
    noise = Noise()
    for out in outputs:
        figures = {}
        for name in out.drives:
            siblings = out.seed_siblings(name)
            if len(siblings) < 2 or len({out.drives[s].seed for s in siblings}) < 2:
                continue
            key = frozenset(siblings)
            noise.member.setdefault(name, []).append(key)
            if key in figures:
                continue
            figures[key] = [out.drives[s].figures() for s in siblings]
            spreads = noise.groups.setdefault(key, {})
            for f in FIGURES:
                s = _spread([fig[f.name] for fig in figures[key]])
                if s is not None:
                    spreads[f.name] = max(spreads.get(f.name, 0.0), s)
    for spreads in noise.groups.values():
        for name, s in spreads.items():
            noise.pooled[name] = max(noise.pooled.get(name, 0.0), s)
    return noise


def noise_table(noise: Noise) -> list[dict]:
    """Per figure: its floor, the largest seed spread, and the threshold a drive without a seed
    group of its own is weighed against (for the report)."""
    return [
        {
            "figure": f.name,
            "label": f.label,
            "floor": f.floor,
            "spread": noise.pooled.get(f.name),
            "threshold": max(f.floor, K * noise.pooled.get(f.name, 0.0)),
            "digits": f.digits,
        }
        for f in FIGURES
    ]
