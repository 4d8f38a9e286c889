"""What a person reads or deploys: the summary and queries of an artefact folder, the figures, the HTML
report and the exported C and Python code."""
