"""knotlab app layer: the `knotlab` command line and the viser labelling web app (`app/web/`)."""
