# Convenience wrappers; ./run does the work (and needs no make on a fresh machine).
.PHONY: demo test
demo:
	./run demo
test:
	./run test
