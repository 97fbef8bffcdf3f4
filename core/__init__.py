"""knotlab core: the science (rope world, knot test, registration, learning); no web, no DB."""
