"""Benchmarks of flexjoint-harness against its peers (``flexjoint bench``); not part of the library."""
