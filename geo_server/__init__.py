"""geo-server: emulator of the TwinCAT 3 CNC GEO task axis compensations."""

__version__ = "0.1.0"
