"""The mission flow, the inbox flow and the command line.

Prefect's client telemetry (and the notice it prints on a first interactive run) is off by
default: ``DO_NOT_TRACK=1`` unless the environment says otherwise, set before Prefect is
imported.
"""
import os as _os

_os.environ.setdefault("DO_NOT_TRACK", "1")
