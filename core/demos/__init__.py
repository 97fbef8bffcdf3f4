"""The data: the demonstration library file, the scripted expert, library generation, task sets."""
