"""The interactive relighting viewer (`lightstage view`): per-view OLAT bases, compressed, in a self-contained
WebGL2 page (docs/viewer.md)."""
