"""unscatter: learned compensation of cell-induced light scattering in DLP bioprinting."""

__version__ = "0.1.0"
