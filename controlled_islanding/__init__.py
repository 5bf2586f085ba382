"""Online PMU-driven controlled islanding (Banna et al., DTW coherency + constrained spectral clustering)."""

__version__ = '0.1.0'
