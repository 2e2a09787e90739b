"""motionforge data package."""
