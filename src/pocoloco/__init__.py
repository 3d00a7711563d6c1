"""pocoloco: point-cloud models of clothed humans in loose clothing."""

__version__ = "0.1.0"
