"""Tests of service.daemon: configuration, the receiver loop, sd_notify, crash safety, systemd."""
