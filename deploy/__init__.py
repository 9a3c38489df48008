"""The command line, fleet runners, reports and plots."""
