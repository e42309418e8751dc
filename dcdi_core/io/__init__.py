"""File input and output: images and depth maps in the project's conventions;
the shipped .npz files' checksum and read-once cache (``npzfile``)."""
