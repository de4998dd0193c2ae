"""Support code for the tests and benches (never imported by the product)."""
