"""ccrp: Clone-based Cloud Robotic Platform."""

__version__ = "0.1.0"
