"""knotlab core: the science (rope world, knot test, registration, learning). No web, no database."""
