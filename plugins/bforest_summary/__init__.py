"""Tree-level summary statistics as a feature set, and a distance between summaries."""
