"""The long-running loop, its configuration and systemd notification."""
