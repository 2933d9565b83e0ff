"""PB3A applications: each runnable as a script and with ``pb3a scenario NAME``."""
