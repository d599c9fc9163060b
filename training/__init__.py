"""The relighting model (volume-rendered radiance-transfer gradient), losses, trainer, eval, relighting, meshes."""
