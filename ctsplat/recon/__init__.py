"""Classical reconstructions: FDK, SIRT/SART, ASD-POCS, MBIR, and their parameters chosen on validation views."""
