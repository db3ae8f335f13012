"""The built-in world's simulator: a generated town or city (:mod:`.town`), drives through it and
spinning LiDARs scanning it (:mod:`.lidar_sim`, :mod:`.lidar_models`). It is one source among
the others: ``core/sequences/sources/town.py`` registers it, and nothing outside the sources and
the benches reaches into it."""
