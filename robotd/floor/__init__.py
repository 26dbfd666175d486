"""The floor loop detector (paper 003): compact descriptors, matching, the map index."""
