"""Per-frame pre-processing: depth validation and back-projection, downsampling, outliers, normals."""
