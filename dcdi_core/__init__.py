"""dcdi_core: depth-aware lens simulation engine (pure numpy; torch only in models/)."""
__version__ = "0.1.0"
