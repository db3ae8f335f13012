"""When the filter is localized, lost or wrong: the paper's localization, false-positive and loss
rules, S2M's confirmation and the whole-map second opinion, the start and frame checks, and how
the truth grades an estimate (never fed back).
"""
