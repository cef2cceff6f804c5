"""Sources of depth frames (all I/O lives here): each yields :class:`elevmap.frame.Frame` records."""
