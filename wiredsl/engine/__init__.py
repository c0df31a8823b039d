"""What turns a Scene into image features: geometry, world arrays, visibility, projection, trials."""
