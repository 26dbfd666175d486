"""robotd: on-robot loop-closure daemon for Turtlebot-class robots."""

__version__ = "0.1.0"
