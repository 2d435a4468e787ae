"""Stage 1, the mesh: reading mesh files, the Mesh type (welding, components, repair), closest points."""
