"""cell: an autonomous active-vision scanning cell.

Layers, imports pointing down: ``cell.cli`` > ``cell.jobs`` > ``cell.planning`` > ``cell.control`` /
``cell.safety`` > ``cell.perception`` > ``drivers``.
"""

__version__ = "0.1.0"
