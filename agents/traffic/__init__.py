"""Traffic control on SUMO: road networks built from files in the repo, legal signal
sequences, the driver that runs a SUMO simulation behind PB3A ports, the junction
controllers (swappable for one another mid-phase), the junction's sensors and the
performance agent that swaps its controller."""
