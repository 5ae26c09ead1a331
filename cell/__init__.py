"""cell: an autonomous active-vision scanning cell.

Layers, imports pointing down: ``cell.api`` / ``cell.cli`` > ``cell.service`` > ``cell.jobs`` >
``cell.planning`` > ``cell.control`` / ``cell.safety`` > ``cell.perception`` > ``drivers``.
"""

__version__ = "0.1.0"
