"""JEPT's model components, one module per part the paper names (Section 3.2, Appendix A.2)."""
