"""The sim-to-real gap: the real experiments re-simulated, the linear parameters recalibrated, the unmodelled
effect found, the gap localised; ``diagnosis.json`` (:mod:`.result`) and the blind test of the diagnoser."""
