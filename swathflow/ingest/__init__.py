"""Stage 1, ingest: a mission folder loaded and checked (every problem at once)."""
