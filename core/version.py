"""lidarloc's version: recorded in every run's recording, exported as ``lidarloc.__version__``."""

VERSION = "0.1.0"
