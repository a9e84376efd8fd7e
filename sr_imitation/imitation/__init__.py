"""The imitation substrate: ACT-SR actor memories, the wake-sleep stream trainer and evaluation."""
