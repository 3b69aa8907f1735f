"""Everything that touches a device: cameras, clocks and sync, LEDs, the recorder, the simulated cube."""
