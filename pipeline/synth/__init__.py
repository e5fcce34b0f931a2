"""Generated underwater scenes with ground truth: the procedural and photo-textured families."""
