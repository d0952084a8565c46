"""Stages 5 and 6: strip systematic-error matching and feathered mosaicking."""
