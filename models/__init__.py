"""motionforge models package."""
