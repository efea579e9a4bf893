"""The coil board's firmware (C sources for the ATmega2560 and the simavr harness), shipped as package
data so `rigctl emulate coil-board --firmware simavr` builds it from an install as from a checkout."""
