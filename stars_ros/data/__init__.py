"""Rating data: SocNav1 and generic loaders, scene graphs and their featurisation, the
encoder-ready scene stores and scene sources for the companion nodes."""
