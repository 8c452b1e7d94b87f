"""What the add-on and the job process share, without torch: job events, run endings, outputs, quality levels."""
