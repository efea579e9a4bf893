"""The Arduino coil board (seed 004): two particles placed by wall contacts, closed loop."""
