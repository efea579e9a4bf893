"""Software emulators of every device, serving the devices' own protocols on real transports."""
