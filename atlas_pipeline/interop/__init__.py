"""What other tools read from a world: trainer exports (COLMAP model, nerfstudio ``transforms.json``)
with the frames at their poses, a triangle mesh (TSDF) and a 2D occupancy grid for navigation."""
