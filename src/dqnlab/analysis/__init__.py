"""Looking at runs, finished or under way: reports, Q-value inspection, videos, sweep status."""
