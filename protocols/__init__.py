"""Transports: sources of phase samples and sinks of drive status, one module per transport,
each with a device-side emulator for tests. The contract is in ``protocols.base``."""
