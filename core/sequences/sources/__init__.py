"""The registered sources, one module each: a module that defines ``SOURCE`` (a
:class:`~lidarloc.core.sequences.registry.Source`) is found by the registry, nothing else to edit.
Each imports what reads its data only when it is opened, so that listing the sources is cheap."""
