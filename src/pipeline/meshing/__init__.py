"""Meshing: TSDF fusion of depth maps (mm) into cleaned triangle meshes."""
