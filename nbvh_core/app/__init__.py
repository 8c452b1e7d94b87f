"""The applications: the compress pipeline, the command line, the add-on's job, library batches, the render worker."""
