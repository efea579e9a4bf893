"""The rig kinds: what differs between the six-coil manipulator, the coil board and the arms."""
