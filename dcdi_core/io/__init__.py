"""File input and output: images and depth maps in the project's conventions."""
