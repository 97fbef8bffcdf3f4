"""Other systems' file formats: demo libraries and labels in the original HDF5 layout."""
