"""flexjoint-harness: FMU co-simulation, ARMAX identification and sim-to-real diagnosis of a flexible joint."""

__version__ = "0.1.0"
