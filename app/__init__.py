"""knotlab app layer: the `knotlab` command line (and, later, the viser web app)."""
