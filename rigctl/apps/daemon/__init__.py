"""The daemon: the service that owns a rig (server), its stream process (runhost), the wire
messages, telemetry, CURVE keys and systemd notification."""
