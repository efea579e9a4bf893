"""Emulated Kepco BOP bipolar supply driving one coil."""
