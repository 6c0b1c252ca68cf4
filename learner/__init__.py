"""Offline application: bags -> TPSR/PCA model -> fitted-Q policy -> evaluation and reports."""
