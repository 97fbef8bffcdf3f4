"""The labelling web app (viser): server, per-tab sessions, scene and panels."""
