"""What every run shares, whatever the rig: states and control, progress, the summary."""
