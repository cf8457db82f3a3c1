import signal
def test_probe():
    print('SIGINT in pytest:', signal.getsignal(signal.SIGINT))
