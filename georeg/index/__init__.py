"""Feature index: geo-referenced map features, the visual-word vocabulary and the inverted file."""
