"""knotlab app layer: the `knotlab` command line (and, later, the viser web app)."""

# What `knotlab --version` reports when knotlab is run from a checkout without being installed;
# keep it equal to pyproject's [project] version.
__version__ = "0.1.0"
