"""Emulated Hall-sensor board of the dual-permanent-magnet rig (seed 003)."""
