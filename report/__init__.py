"""``dtx report``: reports assembled from measurements across the pipeline."""
