"""Emulated KUKA LBR arm: the robot side of the KUKA Sunrise Toolbox TCP protocol (seed 003 rig)."""
