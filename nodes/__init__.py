"""ConstructAide nodes: one folder per node, each with a ``node.py`` declaring its contract and ``main``."""
