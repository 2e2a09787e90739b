"""motionforge pipelines package."""
