"""The one configuration model of a cell (:mod:`cell.config.models`) and its YAML loader."""

from cell.config.load import load_config
from cell.config.models import CellConfig

__all__ = ["CellConfig", "load_config"]
