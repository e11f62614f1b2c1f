"""What a trained run is exported as (`uw-export`): ply.py writes the Gaussians in the 3DGS PLY layout, medium.py the
learned medium as JSON."""
