"""motionforge stages package."""
