"""The dual-EPM rig (seed 003): two KUKA arms carrying permanent magnets and a Hall board."""
