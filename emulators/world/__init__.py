"""The emulated world: robots moved by what the emulated actuators actually do."""
