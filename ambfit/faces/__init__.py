"""What users see: the command line, figures and HTML reports."""
