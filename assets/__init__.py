"""Data files of jaxmm (robot descriptions), installed as the package ``jaxmm.assets``."""
