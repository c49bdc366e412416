"""The package's version, in a module of its own so that code below the package's face can
read it without importing the face (which imports the viewer and the renderer)."""

__version__ = "0.1.0"
