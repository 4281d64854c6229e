"""The two intermediate representations: the graph IR (graph.py) and the loop-nest IR (loops.py)."""
