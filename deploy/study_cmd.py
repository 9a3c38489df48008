"""The study's report under its old module name, for deploy/launch_cmd.py only until that module
moves to deploy/commands/ (issue 12); everyone else imports :mod:`deploy.study_report`."""

from deploy.study_report import render_summary, write_plots

__all__ = ["render_summary", "write_plots"]
