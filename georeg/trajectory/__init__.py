"""Video trajectory: keyframes, SfM, Sim(3), ICP, per-frame tracking and outputs."""
