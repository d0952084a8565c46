"""The mission flow, the inbox flow and the command line."""
