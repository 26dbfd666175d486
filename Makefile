# Thin wrappers around ./dev, which does the setup (see README.md).
.PHONY: demo test test-slow setup
demo:
	./dev demo $(ARGS)
test:
	./dev test $(ARGS)
test-slow:
	./dev test-slow $(ARGS)
setup:
	./dev setup
