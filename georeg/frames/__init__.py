"""Frame geo-localisation: rendering, coarse location, PnP, refinement, outputs."""
