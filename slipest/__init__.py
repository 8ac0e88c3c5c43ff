"""slipest: online slip estimation for wheel-legged rovers from hub vibration."""

__version__ = "0.1.0"
