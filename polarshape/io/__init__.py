"""Input and output: capture folders, result folders, atomic writes."""
