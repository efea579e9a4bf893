"""Device drivers: one module per device family, each on a transport opened from a URL."""
