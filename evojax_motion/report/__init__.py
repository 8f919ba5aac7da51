"""A run's figures (`plots`), motion renderings (`render`) and its HTML report (`build`)."""
