#include "vrpn_server/net/socket_util.h"

#include <gtest/gtest.h>

namespace trackcal::vrpn {
namespace {

in_addr A(const char* s) { return *ParseIpv4(s); }

TEST(AllowList, Nominal) {
  const auto list = AllowList::Parse({"192.168.1.0/24", "10.0.0.7", "127.0.0.0/8"});
  EXPECT_TRUE(list.Allows(A("192.168.1.200")));
  EXPECT_FALSE(list.Allows(A("192.168.2.1")));
  EXPECT_TRUE(list.Allows(A("10.0.0.7")));
  EXPECT_FALSE(list.Allows(A("10.0.0.8")));
  EXPECT_TRUE(list.Allows(A("127.4.5.6")));
}

TEST(AllowList, EmptyAllowsEveryoneAndZeroLengthToo) {
  EXPECT_TRUE(AllowList::Parse({}).Allows(A("8.8.8.8")));
  EXPECT_TRUE(AllowList::Parse({"0.0.0.0/0"}).Allows(A("8.8.8.8")));
  // Host bits in the base are masked away.
  EXPECT_TRUE(AllowList::Parse({"192.168.1.77/24"}).Allows(A("192.168.1.1")));
}

TEST(AllowList, BadEntriesThrowNamingTheEntry) {
  for (const char* bad : {"192.168.1.0/33", "192.168.1/24", "host.example", "1.2.3.4/", "1.2.3.4/x"}) {
    try {
      AllowList::Parse({bad});
      ADD_FAILURE() << bad;
    } catch (const std::invalid_argument& e) {
      EXPECT_NE(std::string(e.what()).find(bad), std::string::npos);
    }
  }
}

TEST(ParseIpv4, RejectsNames) {
  EXPECT_TRUE(ParseIpv4("127.0.0.1"));
  EXPECT_FALSE(ParseIpv4("localhost"));
  EXPECT_FALSE(ParseIpv4("1.2.3.4.5"));
  EXPECT_EQ(FormatEndpoint(MakeSockaddr(A("1.2.3.4"), 3883)), "1.2.3.4:3883");
}

}  // namespace
}  // namespace trackcal::vrpn
