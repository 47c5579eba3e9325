def test_extension_imports():
    import solver_cpp

    assert solver_cpp._core is not None
