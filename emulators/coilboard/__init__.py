"""Emulators of the coil-board rig (seed 004): the firmware on a pty, and the real firmware in simavr."""
