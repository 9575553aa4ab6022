"""Inverse fitting of the medium (sigma_t, g, albedo, light intensity) from target images, with optimistix."""
