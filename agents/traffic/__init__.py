"""Traffic control on SUMO: road networks built from files in the repo, legal signal
sequences, and the driver that runs a SUMO simulation behind PB3A ports."""
