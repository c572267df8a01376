"""The report: tables, figures, small-sample statistics and the paper's claims it tests."""
