"""rigctl: run magnetic micro-robot manipulation rigs."""
