"""Pictures: ray-cast images of fields and paths, coloured PLY meshes."""
