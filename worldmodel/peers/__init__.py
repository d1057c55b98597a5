"""Peer systems brought onto our simulator and yardstick (docs/design.md §10): each module trains its learner
inside ``train_agent`` and evaluates its own scenario family inside ``evaluate family=NAME``."""
