"""Reports of the fit, of the paper's measured series and of a diagnosis (text, markdown, plots)."""
