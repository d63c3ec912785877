"""Built-in recipes (``*.yaml``), installed as the package ``slam.configs``."""
