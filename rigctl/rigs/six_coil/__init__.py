"""The six-coil manipulator (seeds 000 and 002): realize, allocate, the Kepco supplies, global
moves with their camera supervisor, and pair formation with pure pursuit."""
