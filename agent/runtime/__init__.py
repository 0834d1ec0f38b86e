"""The thin runtime around the signal chain: config, journal, systemd notification, CLI, service."""
